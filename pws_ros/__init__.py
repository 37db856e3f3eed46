"""pws_ros: certify image classifiers against camera motion with Pixel-wise Smoothing.

The engine lives in :mod:`pws_ros.core` (ROS-free); ROS 2 nodes in :mod:`pws_ros.nodes`.
"""
__version__ = "0.1.0"
