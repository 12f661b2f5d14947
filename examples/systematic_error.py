"""Systematic ("wiggling") error of each modulation against true distance (SPEC §6 experiment 4, noise-free).

Prints a Markdown table of the peak error and its period per frequency, for square and sine waves with
4 and 3 phase steps, from ``tofcore.sensor.decode.systematic_error_curve`` (ideal single returns, no noise).

Usage: ``.venv/bin/python examples/systematic_error.py``
"""

import numpy as np

from tofcore.sensor.decode import systematic_error_curve
from tofcore.sensor.modulation import Modulation


def main() -> None:
    print("| modulation | f MHz | steps | peak error mm | period m |")
    print("|---|---|---|---|---|")
    for kind in ("cw_square", "cw_sine"):
        for f_mhz in (16, 20, 30, 80, 120):
            for steps in (4, 3):
                mod = Modulation(kind=kind, frequencies_hz=(f_mhz * 1e6,), phase_steps=(steps,))
                d_amb = mod.ambiguity_distances_m()[0]
                d = np.linspace(0.0, d_amb, 20001)
                err = systematic_error_curve(mod, d)[0]
                spectrum = np.abs(np.fft.rfft(err - err.mean()))
                harmonic = int(np.argmax(spectrum[1:]) + 1)  # periods per ambiguity distance
                period = d_amb / harmonic if spectrum.max() > 1e-9 else float("nan")
                print(f"| {kind} | {f_mhz} | {steps} | {np.abs(err).max() * 1000:.2f} | {period:.3f} |")


if __name__ == "__main__":
    main()
