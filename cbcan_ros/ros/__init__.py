"""The ROS 2 layer: the node, its parameters, deferred answers and the command-line client."""
