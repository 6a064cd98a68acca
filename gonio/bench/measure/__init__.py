"""From frames to f_r: HDR merge, one point's reduction, the calibration's alignment
mathematics and its use per point, and the colour matrix.
"""
