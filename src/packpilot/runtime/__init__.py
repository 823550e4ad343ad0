"""PackPilot on a real pack: the BMS runtime over CAN (``run``), the hardware-in-the-loop
twin (``hil``) and the pack as one battery (Pylontech, DroneCAN). See ``docs/runtime.md``."""
