"""Shared mathematics: rigid transforms (``geometry``), the camera model (``camera``), least squares (``lm``)."""
