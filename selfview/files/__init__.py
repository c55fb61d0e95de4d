"""Files: the cell, calibration and camera files, safe bounded reading and writing, the lock folder."""
