"""Image measurement: plates and discs, fingertips and silhouettes (``_csil`` kernel), objects' targets."""
