"""Sensor data -> dataset formats: `lsd3d-usd dataset` (docs/datasets.md).

    timeline   when each sensor fires: cameras, LiDAR and keyframes on one tick grid
    drive      one log (a scene driven along a route): samples rendered one at a time
    tokens     deterministic tokens and microsecond timestamps
    mapping    our classes -> nuScenes categories, attributes from motion, visibility bins
    maps       the drivable area of a layout rasterised as a nuScenes map mask
    writers    the registry of dataset writers (entry-point group lsd3d_usd.dataset_writers)
    nuscenes   the nuScenes v1.0 writer (13 tables, lidarseg, map masks)
    kitti      the KITTI 3D object writer (front camera at keyframes)
    mcap       the MCAP writer with Foxglove schemas
    build      planning a dataset (scenes x routes), checking the output folder, resuming
    commands   the `dataset` CLI

Writers only reformat: they get one Sample (poses, calibrations, images, sweeps, boxes) at a
time from `drive` and own no rendering. Layering: above views, below pipeline.
"""
