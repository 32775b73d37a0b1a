"""The simulated Otbot hardware, behind the same buses as the real robot: CiA 402 drives and the
CiA 406 encoder as CANopen slaves (``canopen_slaves``), the lockstep plant (``plant``), the master's
robot on a virtual bus to it (``bus_robot``), the plant in its own process (``plant_process``), the
VectorNav IMU on a pseudo-terminal (``imu``) and an slcan USB-CAN adapter (``slcan_adapter``).
The numerical simulator they step is ``otbot_hw.simulation``."""
