"""What a run means: series, events, step windows, figures, the summary, plots, Rerun.

The recording (:mod:`adnmesh.recording`) is the file format; this package reads meaning into
it, with one rule for each thing a person looks at, used alike by ``adnmesh up``'s summary,
``inspect``, ``plot``, ``replay``, ``export`` and the live view:

- :mod:`~adnmesh.results.rules`: the one table of what messages mean (series, events);
- :mod:`~adnmesh.results.series`: recorded messages to named time series and events, by those
  rules;
- :mod:`~adnmesh.results.eventlog`: the events as ``foxglove.Log`` records while a run records;
- :mod:`~adnmesh.results.figures`: how P_IP followed each step of P_ref (step windows);
- :mod:`~adnmesh.results.fault_figures`: per fault, detection, deviation and recovery;
- :mod:`~adnmesh.results.summary`: the end-of-run summary;
- :mod:`~adnmesh.results.realtime_report`: what a realtime run says about its own timing;
- :mod:`~adnmesh.results.time_plot`: the paper-style time plot (``adnmesh plot``);
- :mod:`~adnmesh.results.rerun_export`, :mod:`~adnmesh.results.live`: Rerun, after and during a
  run;
- :mod:`~adnmesh.results.csv_export`, :mod:`~adnmesh.results.foxglove_layout`: a run's series
  as CSV files and a Foxglove layout for it (``adnmesh export``).
"""
