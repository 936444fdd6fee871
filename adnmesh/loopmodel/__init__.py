"""The reference loop model and every figure of merit computed from it (pure numerics, no I/O).

- :mod:`~adnmesh.loopmodel.plant`: the reference plant of a DER subset (first-order lags with
  dead time), grouped by identical dynamics;
- :mod:`~adnmesh.loopmodel.frequency_response`: the loop's exact frequency response (delays as
  ``exp(-j omega T)``);
- :mod:`~adnmesh.loopmodel.stability`: certified closed-loop stability (Nyquist winding);
- :mod:`~adnmesh.loopmodel.margins`: disk margin and classical margins;
- :mod:`~adnmesh.loopmodel.step_response`: closed-loop step responses with exact delays;
- :mod:`~adnmesh.loopmodel.step_figures`: the one rule of every step figure (rise, settling,
  overshoot, peak);
- :mod:`~adnmesh.loopmodel.evaluation`: all figures of merit of many candidate PI pairs at once;
- compiled kernels (numba): :mod:`~adnmesh.loopmodel.step_kernels`,
  :mod:`~adnmesh.loopmodel.settle_kernel`, :mod:`~adnmesh.loopmodel.frequency_kernels`.

The method behind them: ``docs/method.md``.
"""
