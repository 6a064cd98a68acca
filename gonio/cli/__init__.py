"""The ``gonio`` command line: argument parsing, and one command module per use case that
calls the library.
"""
