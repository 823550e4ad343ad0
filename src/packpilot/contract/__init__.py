"""The contracts every layer shares; this package imports nothing of PackPilot.

* :mod:`.bms` — what a controller sees and says: measurements, commands, events, the
  controller protocol (the scalar, one-pack form);
* :mod:`.arrays` — the same for P packs at once, as arrays (what the compiled core reads and
  writes), and the conversions between the two forms;
* :mod:`.events` — the reason tables that turn event codes into :class:`~.bms.Event` objects;
* :mod:`.charger` — charger command and status with the one list of charger flags, and the
  link that carries them (direct or CAN);
* :mod:`.topology` — the pack's batteries and the one battery index (string / traction /
  display name);
* :mod:`.record` — what a run records (samples, trace, result) and where it goes.
"""
