"""Exports of a session to files other tools open: ROS bags (:mod:`.bag`)."""
