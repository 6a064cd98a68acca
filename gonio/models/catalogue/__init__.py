"""The registered models, one file a model: its parameters, its numpy formula, its Dr.Jit
kernel and its Mitsuba 3 twin.
"""
