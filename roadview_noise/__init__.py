"""rvnoise: compound sensor noise models (EU ROADVIEW D3.5) for camera, LiDAR and 4D radar data."""

__version__ = "0.1.0"
