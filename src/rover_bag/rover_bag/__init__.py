"""Record and replay rosbag2 (MCAP) bags; a DDS-free batch reader for offline tools."""
