"""Force models for the simulated rig: what the specimen pushes back with.

A model maps the probe's whole travel history to the force on the probe, so a
time-dependent specimen can be modelled. It is the only coupling between the
simulated rig and a specimen: the finite-element model plugs in here too.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np


@runtime_checkable
class ForceModel(Protocol):
    def force_N(self, time_s: np.ndarray, displacement_mm: np.ndarray) -> np.ndarray:
        """Force on the probe (N, positive = compression) at each time of the history.

        ``time_s`` (increasing) and ``displacement_mm`` (probe travel from the
        stage's zero, positive = towards/into the specimen) are the whole history
        so far; the result has the same length. Models must be causal: entry i
        may depend on entries 0..i only. The simulated sensor reads the last
        entries; it calls the model once per batch of new samples.
        """


@dataclass(frozen=True)
class NonlinearSpring:
    """F = k d + k3 d^3 for indentation d = travel - contact_mm > 0, else 0 (no contact).

    ``contact_mm`` is the gap the probe travels before it first touches.
    """

    k_N_per_mm: float = 1.0
    k3_N_per_mm3: float = 0.05
    contact_mm: float = 2.0

    def elastic_N(self, displacement_mm: np.ndarray) -> np.ndarray:
        d = np.maximum(np.asarray(displacement_mm, float) - self.contact_mm, 0.0)
        return self.k_N_per_mm * d + self.k3_N_per_mm3 * d**3

    def force_N(self, time_s: np.ndarray, displacement_mm: np.ndarray) -> np.ndarray:
        return self.elastic_N(displacement_mm)

    def depth_for_force_mm(self, force_N: float) -> float:
        """Indentation (from contact) at which the elastic force equals ``force_N``."""
        roots = np.roots([self.k3_N_per_mm3, 0.0, self.k_N_per_mm, -force_N]) if self.k3_N_per_mm3 else \
            np.array([force_N / self.k_N_per_mm])
        real = roots[np.abs(roots.imag) < 1e-9].real
        return float(real[real >= 0].min())


@dataclass(frozen=True)
class ViscoelasticSpring:
    """The nonlinear spring with one-term Prony relaxation (quasi-linear viscoelasticity).

    G(t) = g_inf + g1 exp(-t / tau1), g_inf = 1 - g1; F(t) = integral of G(t - s) dF_e(s),
    with F_e the spring's elastic force. Held at a fixed depth the force relaxes
    from F_e to g_inf F_e with time constant tau1. The force never pulls (>= 0).
    """

    spring: NonlinearSpring = field(default_factory=NonlinearSpring)
    g1: float = 0.3
    tau1_s: float = 2.0

    @property
    def contact_mm(self) -> float:
        return self.spring.contact_mm

    def force_N(self, time_s: np.ndarray, displacement_mm: np.ndarray) -> np.ndarray:
        t = np.asarray(time_s, float)
        fe = self.spring.elastic_N(displacement_mm)
        if t.size == 0:
            return fe
        dfe = np.diff(fe, prepend=0.0)
        h = prony_memory(t, dfe, self.tau1_s)
        return np.maximum((1.0 - self.g1) * fe + self.g1 * h, 0.0)


def prony_memory(t: np.ndarray, increments: np.ndarray, tau_s: float) -> np.ndarray:
    """h_i = sum_{j<=i} exp(-(t_i - t_j) / tau) increments_j, vectorised and overflow-safe.

    Computed block by block (each block spans < 50 tau) with the block start as
    the reference time, carrying the memory from block to block.
    """
    n = t.size
    out = np.empty(n)
    carry, t_carry = 0.0, t[0]
    start = 0
    while start < n:
        stop = int(np.searchsorted(t, t[start] + 50.0 * tau_s, side="left"))
        stop = max(stop, start + 1)
        tb = t[start:stop] - t[start]
        w = np.exp(tb / tau_s)
        acc = np.cumsum(increments[start:stop] * w) / w
        acc += carry * np.exp(-(t[start:stop] - t_carry) / tau_s)
        out[start:stop] = acc
        carry, t_carry = acc[-1], t[stop - 1]
        start = stop
    return out
