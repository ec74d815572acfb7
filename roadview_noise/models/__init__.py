"""Models: one module per phenomenon, grouped by sensor. Every module is imported by registry.load_all()."""
