"""``jetbot-rt calibrate``: the drive programme (``programme``), the marker measurement
(``measure``) and the fit (``fit``). Robot side: Python 3.8, numpy and OpenCV only."""
