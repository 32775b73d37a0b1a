"""Numerical simulation of Otbot: zero-order-hold integration of the paper's model and of the
extended model (``simulator``), simulated runs turned into recordings (``runs``), and runs with a
concealed effect for proving the mismatch finder (``concealed``). Pure computation: no bus, no
simulated hardware (that is ``sim/``)."""
