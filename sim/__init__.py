"""gonio.sim."""
