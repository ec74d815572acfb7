"""Built-in sensor profiles and loaders from files (camera intrinsics, LiDAR beam tables, radar parameters)."""
