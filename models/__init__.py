"""gonio.models."""
