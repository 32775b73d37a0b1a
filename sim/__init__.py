"""The simulated Otbot: integration of the model (``sim.simulator``) and, behind the
same buses as the real robot, simulated CANopen devices and IMU."""
