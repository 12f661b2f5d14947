"""Frames with few valid pixels: the warning that names the likely reason.

A frame whose scene lies beyond the sensor's range, or faces away from its LEDs, decodes to almost no
valid pixel; its numbers (an RMS error over a handful of pixels) then mislead. :func:`low_coverage`
turns such a frame into one line: the share of valid pixels and the most common reason of the others
(the ``reason`` image, :class:`tofcore.sensor.decode.Reason`), with what to do about it. The
``tofcore render`` command prints it, ``tofcore-batch`` records it (``warning`` in the frame's record)
and the Blender add-on reports it.

============================  ==========================================================================
most common reason            the line says
============================  ==========================================================================
out of range                  the surfaces are beyond the sensor's range: move it closer
no return, low amplitude      no (or too little) LED light returns: nothing in view, surfaces too far,
                              dark or facing away
saturated                     too much light: surfaces too close or too bright
unwrapping failed             the modulation frequencies disagree (multipath, noise)
============================  ==========================================================================
"""

from __future__ import annotations

import numpy as np

#: Below this share of valid pixels a frame gets the warning.
LOW_VALID_FRACTION = 0.10

_WHY = {
    "BEYOND_RANGE": "see surfaces beyond the sensor's range ({range}; the farthest at {far:.1f} m): move the sensor "
                    "closer (or pick a preset with a longer range)",
    "NOTHING": "see no surface, so no LED returns: aim the sensor at the scene",
    "OUT_OF_RANGE": "are decoded outside the sensor's range ({range}): move the sensor closer or away",
    "NO_RETURN": "get no LED return (surfaces facing away): aim the sensor at the scene",
    "LOW_AMPLITUDE": "get too little LED light back (surfaces too far, too dark or facing away): "
                     "move the sensor closer",
    "SATURATED": "are saturated (surfaces too close or too bright): move the sensor away or shorten the "
                 "exposure",
    "UNWRAPPING_FAILED": "failed unwrapping (the modulation frequencies disagree: multipath or noise)",
}


def low_coverage(frame, threshold: float = LOW_VALID_FRACTION) -> str | None:
    """None when at least ``threshold`` of the frame's pixels are valid, else one line: the valid share and
    the most common cause among the invalid pixels, with its share of all pixels and what to do.

    Among the invalid pixels that see a surface, the ground truth names the cause first: one whose true
    depth is beyond the sensor's longest range is "beyond range" (its weak return often decodes as low
    amplitude); the others count by their ``reason`` code. The pixels that see no surface are added as a
    share; where no pixel sees one, that is the cause.
    """
    from ..sensor.decode import Reason

    valid = np.asarray(frame.valid, dtype=bool)
    fraction = float(valid.mean()) if valid.size else 0.0
    if fraction >= threshold:
        return None
    truth = np.asarray(frame.gt_depth, dtype=np.float64)
    range_m = (frame.metadata.get("sensor") or {}).get("range_m")
    seen = np.isfinite(truth)
    beyond = seen & (truth > range_m[1]) if range_m else np.zeros_like(seen)
    nothing = int(np.sum(~valid & ~seen))
    counts = {"BEYOND_RANGE": int(np.sum(~valid & beyond))}
    rest = np.asarray(frame.reason)[~valid & seen & ~beyond]
    for code, n in zip(*np.unique(rest, return_counts=True)):
        counts[Reason(int(code)).name] = int(n)
    cause = max(counts, key=counts.get)
    if counts[cause] == 0:  # no pixel sees a surface
        cause, counts[cause], nothing = "NOTHING", nothing, 0
    if counts[cause] == 0:
        return None
    why = _WHY.get(cause, cause.lower().replace("_", " ")).format(
        range=f"{range_m[0]:g}-{range_m[1]:g} m" if range_m else "its range",
        far=float(np.max(truth[seen])) if seen.any() else float("nan"))
    return (f"only {100 * fraction:.1f} % of the pixels are valid (fewer than {100 * threshold:.0f} %): "
            f"{100 * counts[cause] / valid.size:.0f} % {why}"
            + (f"; {100 * nothing / valid.size:.0f} % see no surface" if nothing else ""))
