"""Procedural "ideal drive" generator for camera, raw Bayer, LiDAR and radar sample data."""
