"""Plants on the other end of a real protocol (docs/devices.md).

- :mod:`~adnmesh.devices.link`: what the DER agent's gateway needs of a device connection
  (:class:`~adnmesh.devices.link.DeviceLink`), the readings it gets and the errors it tells apart;
- :mod:`~adnmesh.devices.gateway`: the gateway thread around a link and the device's health;
- :mod:`~adnmesh.devices.sunspec`: Modbus TCP with the SunSpec DER models (pymodbus, the
  model definitions of pysunspec2): a client link and a device simulator's server;
- :mod:`~adnmesh.devices.iec104`: IEC 60870-5-104 (c104): a client link and a device
  simulator's server;
- :mod:`~adnmesh.devices.realtime_plant`: a DER's model run on the wall clock, what the device
  simulators serve; :mod:`~adnmesh.devices.faults`: the faults they can play;
- :mod:`~adnmesh.devices.connect`: the objects above from a DER's ``plant:`` section.
"""
