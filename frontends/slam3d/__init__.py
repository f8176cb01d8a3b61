"""3D LiDAR SLAM: KISS-ICP odometry, keyframes and verified loop closures into a pose graph."""
