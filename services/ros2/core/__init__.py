"""The pure part of the ROS 2 bridge: key expressions and tokens (``names``), messages (``messages``), the
trajectory the bridge keeps (``trajectory``). No Zenoh, no files."""
