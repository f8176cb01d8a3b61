"""Payload decoding: ROS messages from CDR (ROS 2) or ROS 1 serialization, Foxglove schemas from protobuf or
JSON. Each function here turns bytes into plain fields; `frontends.logs.converters` turns fields into our
types."""
