"""Files: the cell description (``cell``), calibration and camera files (``calfile``, ``camfile``), the atomic,
bounded reading and writing under them (``io_safe``) and the lock folder (``lockdir``)."""
