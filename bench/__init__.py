"""The benchmarks: scripts that print one JSON object each (``selfview report`` runs them all)."""
