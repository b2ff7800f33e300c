"""The CANopen core: one bus, its supervision, SDO, NMT; it knows nothing of ROS."""
