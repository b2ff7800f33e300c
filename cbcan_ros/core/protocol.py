"""Numbers of CiA 301 that every service shares, below all of them."""

MAX_NODE_ID = 127  # node ids are 1..127; 0 addresses all nodes (NMT) or the gateway itself
