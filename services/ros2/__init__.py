"""ROS 2 over Zenoh, no ROS install needed: KM-ViPE's poses, path, map and intrinsics published as ROS 2 messages
(``kmvipe ros2 bridge``), and ROS 2 images read from a live topic (``ros2:/camera/image_raw``) or a bag.
Both ways speak rmw_zenoh's keys or zenoh-bridge-ros2dds's (``KMVIPE_ROS2_FORM``); see README.md here."""
