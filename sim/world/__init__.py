"""The simulated world the camera sees: people (``crowd``, ``walkers``, ``dronecrowd``), the ground
(``ground``), the render (``render``) and the camera served as MJPEG (``camera_server``), also
riding on an external vehicle's pose (``pose_follow``). Knows nothing of the simulated vehicle.
"""
