"""gonio.fitting."""
