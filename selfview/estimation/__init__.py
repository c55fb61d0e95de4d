"""Estimation: Tsai's method, the PCC, off-line and on-line calibration, the policy, the interior orientation."""
