"""Models: one module per phenomenon, grouped by sensor. registry.load_all() imports every module; a run imports only
its recipe's, through model_index.py (``python -m roadview_noise.registry`` regenerates it)."""
