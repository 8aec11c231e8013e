"""usdview plugin: an "LSD3D" menu (render surfels from the current camera, compare GGDS
runs by muting layers, surfel statistics). The work is in ``actions`` (plain functions of a
stage, camera and prims); ``plugin`` holds the PluginContainer. See docs/usdview.md."""
