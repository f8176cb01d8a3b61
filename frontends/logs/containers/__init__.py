"""Container readers (MCAP, ROS 1 bag, ROS 2 bag): find and unpack messages, never decode payloads."""
