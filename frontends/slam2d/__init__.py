"""2D laser SLAM: scan-matching odometry, keyframes and verified loop closures into a pose graph."""
