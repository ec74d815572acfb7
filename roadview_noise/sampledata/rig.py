"""The sample drive's sensor rig: mounts, raw levels, and the reduced preset of the committed sample_data/."""

from __future__ import annotations

SEQUENCE = "seq0"
#: sensor mounts in the ego frame (x forward, y left, z up; origin on the ground under the rear axle), metres;
#: the camera height is the camera profile's ``height_above_ground_m``. No sensor is rotated against the ego frame.
CAMERA_MOUNT_XY_M = (1.5, 0.0)
LIDAR_MOUNT_M = (1.2, 0.0, 1.9)
RADAR_MOUNT_M = (3.7, 0.0, 0.5)
RAW_PATTERN, RAW_BLACK_DN, RAW_WHITE_DN = "RGGB", 64, 4095
#: the committed sample_data/ (size budget ≤ 10 MB): arguments of ``generate``
COMMITTED = {"frames": 3, "seed": 0, "camera_size": (484, 366), "lidar_columns": 256}
