"""What a fit compares: losses, the model's discrepancy term, the instrument's aperture
response and the fit problem (f_r at fixed directions, residuals, Jacobians).
"""
