"""PyBullet two-rover world of Sujan (2002) and the rclpy node that publishes it."""
