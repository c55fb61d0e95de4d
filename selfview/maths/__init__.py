"""Shared mathematics below the rest: rigid transforms (``geometry``), the camera model (``camera``) and the least-squares solver (``lm``)."""
