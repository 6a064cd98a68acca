"""How sure a fit is: the propagated budget (GUM), the posterior (emcee), the Cramer-Rao
bound.
"""
