"""Benchmark: interaction kernels (samples/s of ``interact``, ``transport_coefficients``,
``lookup``, Klein–Nishina).

Run: ``python bench/bench_physics.py [--samples 2000000]``. Builds the tables (timed), compiles
the kernels with a small warm-up call (timed separately), then times single-threaded loops of
each kernel at a few energies in water and cortical bone. Baseline in the same process: the cost
of the RNG alone (``next_uniform``), which every sample pays at least once.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from numba import njit

from tetdose._random import next_uniform, seed_for
from tetdose.transport.physics._photon import (
    interact,
    lookup,
    sample_klein_nishina,
    transport_coefficients,
)
from tetdose.transport.physics.xs import build_cross_sections


@njit(cache=True)
def _loop_interact(xs, material, energy_mev, n, seed):
    state = seed_for(seed, 0, 0)
    total = 0.0
    for _ in range(n):
        state, _, deposited, _, _, _, _, _, _, _, _ = interact(
            xs, material, energy_mev, 0.0, 0.0, 1.0, state)
        total += deposited
    return total


@njit(cache=True)
def _loop_lookup(xs, material, energy_mev, n, seed):
    state = seed_for(seed, 0, 0)
    total = 0.0
    for _ in range(n):
        state, r = next_uniform(state)
        _, inc, pe, pair, mu_en = lookup(xs, material, energy_mev * (0.5 + r))
        total += inc + pe + pair + mu_en
    return total


@njit(cache=True)
def _loop_transport(xs, material, energy_mev, n, seed):
    state = seed_for(seed, 0, 0)
    total = 0.0
    for _ in range(n):
        state, r = next_uniform(state)
        mu, mu_en = transport_coefficients(xs, material, energy_mev * (0.5 + r))
        total += mu + mu_en
    return total


@njit(cache=True)
def _loop_kn(energy_mev, n, seed):
    state = seed_for(seed, 0, 0)
    total = 0.0
    for _ in range(n):
        state, e_out, _ = sample_klein_nishina(energy_mev, state)
        total += e_out
    return total


@njit(cache=True)
def _loop_rng(n, seed):
    state = seed_for(seed, 0, 0)
    total = 0.0
    for _ in range(n):
        state, r = next_uniform(state)
        total += r
    return total


def _rate(fn, *args, n: int) -> float:
    t0 = time.perf_counter()
    fn(*args, n, 1)
    return n / (time.perf_counter() - t0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=2_000_000)
    n = parser.parse_args().samples

    t0 = time.perf_counter()
    xs = build_cross_sections(["water", "cortical_bone"])
    print(f"build_cross_sections (2 materials, {xs.mu_rho_cm2_g.shape[1]} energies): "
          f"{time.perf_counter() - t0:.3f} s")
    t0 = time.perf_counter()
    _loop_interact(xs, 0, 1.0, 10, 0)
    _loop_lookup(xs, 0, 1.0, 10, 0)
    _loop_transport(xs, 0, 1.0, 10, 0)
    _loop_kn(1.0, 10, 0)
    _loop_rng(10, 0)
    print(f"compile / cache load: {time.perf_counter() - t0:.3f} s")

    rng_rate = _rate(_loop_rng, n=n)
    print(f"next_uniform baseline: {rng_rate / 1e6:8.1f} M/s")
    for energy in (0.03, 0.1, 1.0, 10.0):
        kn = _rate(_loop_kn, energy, n=n)
        look = _rate(_loop_lookup, xs, 0, energy, n=n)
        coeff = _rate(_loop_transport, xs, 0, energy, n=n)
        rates = [_rate(_loop_interact, xs, m, energy, n=n) for m in (0, 1)]
        print(f"E = {energy:5.2f} MeV: interact water {rates[0] / 1e6:6.2f} M/s, "
              f"bone {rates[1] / 1e6:6.2f} M/s; lookup {look / 1e6:6.2f} M/s; "
              f"transport_coefficients {coeff / 1e6:6.2f} M/s; "
              f"Klein–Nishina {kn / 1e6:6.2f} M/s "
              f"({np.float64(rng_rate / kn):.1f}× the RNG cost)")


if __name__ == "__main__":
    main()
