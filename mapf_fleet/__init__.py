"""mapf_fleet: learned multi-agent path finding (DHC/DCC with cooperative rewards) on a ROS 2 fleet."""

__version__ = "0.1.0"
