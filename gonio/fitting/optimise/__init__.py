"""Finding the parameters: the parameter space, starts, Levenberg-Marquardt, the affine
fast path, the energy constraint, and the constrained maximum-likelihood fit.
"""
