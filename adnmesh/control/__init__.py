"""The agents' logic as bus-free state machines (see :mod:`adnmesh.control.base`).

- :class:`~adnmesh.control.cpfc_controller.CPFC`: gain-scheduled PI control of ``P_IP``;
- :class:`~adnmesh.control.der_controller.DERController`: a DER's local controller and dynamics;
- :class:`~adnmesh.control.measurement_point.Measurement`: ``P_IP`` at the interconnection point;
- :class:`~adnmesh.control.availability_monitor.AvailabilityMonitor`: heartbeats to SI.

:func:`~adnmesh.control.registry.build_agent` makes the state machine of an agent id. The
control layer imports the wire layer and the numerics, never the sim layer or the runtime.
"""
