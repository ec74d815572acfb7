"""Depth maps as users have them: holes (:mod:`.holes`), per-image calibration files (:mod:`.calibration`), and
depth from other data when there is no depth map — a paired LiDAR scan (:mod:`.lidar`), a monocular depth model
(:mod:`.monocular`) or a flat-road prior (:mod:`.ground_plane`) with vertical objects standing on it
(:mod:`.stixels`). Pure array code plus the readers these need; the recipe's ``inputs`` choose among them in
:mod:`roadview_noise.camera_inputs`."""
