"""An ADN from a grid model: the survey of a SimBench net's static generators, the rules that
make some of them actuators, their default dynamics and a scenario template — what
``adnmesh init`` writes a config from (docs/configuration.md#adnmesh-init).

- :mod:`~adnmesh.adn.dynamics`: the documented default T_delay and T_rise per DER type, and
  which DER type each SimBench generator type is;
- :mod:`~adnmesh.adn.survey`: the net's generators at a study case and P_IP there (imports
  simbench and pandapower);
- :mod:`~adnmesh.adn.selection`: the actuator rules (pure);
- :mod:`~adnmesh.adn.template`: schedules and a scenario sized to the controllable range (pure);
- :mod:`~adnmesh.adn.config_text`: the commented YAML.
"""
