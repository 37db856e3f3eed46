"""ROS 2 nodes (thin rclpy glue around :mod:`pws_ros.bridge` and :mod:`pws_ros.core`).

``cloud_listener``, ``partition_planner``, ``projector``, ``certifier`` (the four-process mode) and
``pipeline`` (the four in one process). rclpy is imported only inside :mod:`._ros`, which the node
modules import when a node starts: every module here imports without ROS; ``main()`` then exits
with a clear message (status 2).
"""
NODE_MODULES = ("cloud_listener", "partition_planner", "projector", "certifier", "pipeline")
