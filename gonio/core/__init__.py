"""What every layer shares and nothing else: geometry, errors a user can act on, the atomic
writer, session file helpers, and the checks before work starts. Imports nothing of gonio.
"""
