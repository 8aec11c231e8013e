"""Stage -> pictures: render a composed scene from a camera at a time, sensor rigs driven
along a route, video clips, and the `render` command.

    stage_data   reading a composed stage into arrays: surfels, env map, actors at a time
    frame        one frame: surfels + actors composited over the env (`render_scene`)
    images       tone mapping, sRGB, reading and writing image files
    preview      `render --camera`: frames of one USD camera
    rigs         rig specs (the Waymo-like five-camera rig)
    ego          ego trajectories: along lanes (IDM or constant speed) or from a pose list
    rig_stage    the rig's USD layer (animated cameras + ego car, sublayering the scene)
    rig          `render --rig`: every camera of a rig at every frame, MP4 per camera
    video        MP4 writing
    deferred     deferred rendering: frames through the scene's image prior (render/eval --deferred)
    scene_cameras  the scene's cameras layer (GGDS views and overviews under /World/Cameras)
    commands     the `render` CLI

Layering: above actors and ggds, below pipeline; render/ is only the rasteriser.
"""
