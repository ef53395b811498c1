"""ROS 2 over rmw_zenoh: the link that wires it into a server and the bridge that speaks the wire.
"""
