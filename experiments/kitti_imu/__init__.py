"""The KITTI IMU + GPS noise-learning protocol (docs/tutorial/imu.md)."""
