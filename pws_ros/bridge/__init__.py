"""ROS-free glue between ROS 2 messages and the core engine.

Everything here works with *duck-typed* messages: rclpy messages and rosbags messages share their
field names, so the same code converts a live message in a node and a recorded one in a test or in
``pws replay``. Nothing in this package imports rclpy (the nodes in :mod:`pws_ros.nodes` do).

- :mod:`.params`      the parameter table (one source of truth) and the validation of a value
- :mod:`.config`      ``PwsConfig`` (built from the table), cross-parameter rules, ``config/pws.yaml`` loading
- :mod:`.paramdoc`    ``config/pws.yaml`` and the parameter table of ``docs/ros2.md``, generated from the table
- :mod:`.msgconv`     messages -> numpy / core objects (images, depth, CameraInfo, RGB-D, transforms)
- :mod:`.cloudconv`   PointCloud2 -> arrays, a Cloud and the camera to render it with
- :mod:`.msgtypes`    the ``types`` namespace of message classes and the basic pieces (headers, poses)
- :mod:`.msgbuild`    core objects -> sensor messages (Image, CameraInfo, PointCloud2, PoseArray);
  re-exports msgtypes and diagnostics
- :mod:`.diagnostics` the certification DiagnosticArray (its key schema), markers, health status
- :mod:`.sync`        stamp matching, the latest-only online policy
- :mod:`.timejump`    time jumping back: a new timeline for every stamp-ordered buffer
- :mod:`.assembly`    partition-set assembly of the four-process mode
- :mod:`.inputs`      the camera-input front end of cloud_listener/pipeline (and pws replay)
- :mod:`.scheme`      the wire scheme of the four-process mode (plans, frames, bounds on topics)
- :mod:`.engine`      ``FrameCertifier``: the per-frame pipeline (plan, render, certify every axis)
- :mod:`.axis_threads` a frame's axes at the same time (``axis_threads``): how many, and the threads that run them
- :mod:`.selfaudit`   the self-audit of a certificate (``audit_every``)
- :mod:`.preview`     preview frames for humans (``rendered/preview``)
- :mod:`.outputs`     one frame's outputs in publication order (the nodes publish them, replay writes them)
"""
