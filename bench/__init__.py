"""gonio.bench."""
