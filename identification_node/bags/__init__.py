"""rosbag2 reading and writing (mcap, sqlite3)."""
