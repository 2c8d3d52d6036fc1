"""Estimation: motion models, observation model, EKF/NH∞, map, cooperation (`fuse`)."""
