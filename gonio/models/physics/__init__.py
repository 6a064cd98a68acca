"""The formulas of reflection in numpy: microfacet distributions, Fresnel terms, diffuse
terms, roughplastic's tables and the directional albedo.
"""
