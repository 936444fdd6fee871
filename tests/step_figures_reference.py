"""The step-figure rule of :func:`adnmesh.loopmodel.step_kernels.accumulate` in plain numpy (vectorised over
the responses), the reference the compiled kernel is tested against (test-only code)."""
import numpy as np


def _vertex(ym, yc, yp, jj, tt, t0, h, inner):
    """Peak and its time per row: the concave parabola's vertex where ``inner``, else sample."""
    if tt is None:
        den = ym - 2 * yc + yp
        off = np.where(inner & (den < 0), 0.5 * (ym - yp) / np.where(den < 0, den, -1.0), 0.0)
        return yc - 0.25 * (ym - yp) * off, t0 + h * (jj + off)
    jm, jp = np.maximum(jj - 1, 0), np.minimum(jj + 1, tt.size - 1)
    d1 = np.where(inner, tt[jj] - tt[jm], 1.0)
    d2 = np.where(inner, tt[jp] - tt[jj], 1.0)
    s1 = (yc - ym) / d1
    a = ((yp - yc) / d2 - s1) / (d1 + d2)
    concave = inner & (a < 0)
    a = np.where(concave, a, -1.0)
    b = s1 + a * d1
    return np.where(concave, yc - b * b / (4.0 * a), yc), np.where(concave, tt[jj] - b / (2.0 * a),
                                                                   tt[jj])


def accumulate_numpy(acc, t0: float, h: float, chunk: np.ndarray, times=None) -> None:
    """Update the state of a :class:`adnmesh.loopmodel.step_figures.StepFigureAccumulator` ``acc`` with
    ``chunk`` (M, n) exactly as its compiled :meth:`add` does (uniform grid, or ``times``)."""
    tt = None if times is None else np.asarray(times, float)

    def time_at(i, frac):
        return t0 + h * (i + frac) if tt is None else tt[i] + (tt[i + 1] - tt[i]) * frac

    y = np.concatenate([acc.last[:, None], chunk], axis=1)     # position 0 = last
    rows = np.arange(y.shape[0])
    for level, store in ((0.1, acc.t10), (0.9, acc.t90)):
        above = y >= level
        idx = np.argmax(above, axis=1)
        hit = above[rows, idx] & (idx > 0) & np.isnan(store)
        i = idx[hit]
        y0, y1 = y[hit, i - 1], y[hit, i]
        store[hit] = time_at(i - 1, (level - y0) / (y1 - y0))
    j = np.argmax(y, axis=1)
    better = y[rows, j] > acc.peak
    if np.any(better):
        jj = j[better]
        yc = y[better, jj]
        ym = y[better, np.maximum(jj - 1, 0)]
        yp = y[better, np.minimum(jj + 1, y.shape[1] - 1)]
        inner = (jj > 0) & (jj < y.shape[1] - 1)
        acc.peak[better], acc.peak_t[better] = _vertex(ym, yc, yp, jj, tt, t0, h, inner)
    for b, band in enumerate(acc.bands):
        store = acc.settle[b]
        out = np.abs(y - 1.0) > band
        any_out = out.any(axis=1)
        last = y.shape[1] - 1 - np.argmax(out[:, ::-1], axis=1)
        ends_out = any_out & (last == y.shape[1] - 1)
        store[ends_out] = np.inf
        cross = any_out & ~ends_out
        i = last[cross]
        y0, y1 = y[cross, i], y[cross, i + 1]
        target = np.where(y0 > 1.0, 1.0 + band, 1.0 - band)
        store[cross] = time_at(i, (target - y0) / (y1 - y0))
    acc.last = chunk[:, -1].copy()
