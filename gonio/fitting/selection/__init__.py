"""Model selection: model only what the data needs (information criteria), or only what a
scene shows (rendered candidates).
"""
