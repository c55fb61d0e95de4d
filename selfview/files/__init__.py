"""Files: cell description, calibration and camera files, bounded reads and atomic writes (``io_safe``), locks."""
