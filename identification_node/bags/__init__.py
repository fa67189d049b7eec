"""rosbag2 bags (mcap, sqlite3): reading (``reader``), writing (``writer``), mcap chunk
checksums (``mcap_check``)."""
