"""calib tests."""
