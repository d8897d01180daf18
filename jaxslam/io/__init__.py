"""Log readers and writers: ROS bags, CARMEN logs, relations files, maps, trajectories."""
