"""The compiled evaluation engine: the models' formulas as Dr.Jit (LLVM) kernels, their
recordings, in-kernel reductions, and the numpy round trip of ``Model.eval``.
"""
