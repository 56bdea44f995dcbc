"""Motion between frames, the sources a run predicts with: odometry (recorded, noisy ground
truth, feature and dense visual odometry: :mod:`.odometry`) and the IMU (samples cleaned,
gaps bridged, preintegrated for GTSAM: :mod:`.imu`)."""
