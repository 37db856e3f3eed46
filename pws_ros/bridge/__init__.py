"""ROS-free glue between ROS 2 messages and the core engine.

Everything here works with *duck-typed* messages: rclpy messages and rosbags messages share their
field names, so the same code converts a live message in a node and a recorded one in a test or in
``pws replay``. Nothing in this package imports rclpy (the nodes in :mod:`pws_ros.nodes` do).

- :mod:`.msgconv`  messages -> numpy / core objects (images, depth, CameraInfo, PointCloud2, RGB-D)
- :mod:`.msgbuild` core objects -> messages (DiagnosticArray certification, PoseArray, PointCloud2,
  Image, MarkerArray, health) for a ``types`` namespace of message classes
- :mod:`.sync`     stamp matching, the latest-only online policy, partition-set assembly
- :mod:`.inputs`   the camera-input front end of cloud_listener/pipeline (and pws replay)
- :mod:`.config`   the parameter table (one source of truth) and ``config/pws.yaml`` loading
- :mod:`.scheme`   the wire scheme of the four-process mode (plans, frames, bounds on topics)
- :mod:`.engine`   ``FrameCertifier``: the per-frame pipeline (plan, render, certify every axis)
- :mod:`.outputs`  one frame's outputs in publication order (the nodes publish them, replay writes them)
"""
