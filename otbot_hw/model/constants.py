"""Physical constants of the model, written once."""

GRAVITY = 9.80665  # m/s^2, standard gravity: the IMU's z reading at rest, the weight in rolling resistance
