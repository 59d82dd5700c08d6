"""UWB ranging (Paper 003): range models, the collaborative UWB EKF, survey range factors."""
