"""Plain-Python reference implementations of the paper's crusher and mill
equations (section "Simulator", errata in fmus/README.md), written independently
of the C model sources, for the FMU tests."""

from __future__ import annotations

import math

import numpy as np

from cosim import sizes

D = [1e-5 * (10 ** (1 / 3)) ** k for k in range(16)]

MILL_DEFAULTS = dict(m0=1000.0, mu_dr=0.02, g=9.8, r_mill=5.0, omega_crit=1.5, d_gr=1e-3,
                     k_gr=1.0, d_cl=2.5e-5, k_cl=10.0, k_esc=1000.0, d_gr_a=1e-3, k_gr_a=1.0,
                     impact_energy=5.8e-5, breakage_energy=1.0, speed_time_constant=5.0,
                     initial_speed=1.2)


def crusher(zone_hardness_mass, speed, gap_width=0.25, k_oversize=1.0, k_undersize=0.1):
    """Eq. crusher_torque, P = tau omega, and the jaw's fragmentation map."""
    oversize = [d >= gap_width for d in D]
    torque = sum((k_oversize if o else k_undersize) * m for o, m in zip(oversize, zone_hardness_mass))
    n_under = oversize.count(False)
    fmap = [[0.0] * 16 for _ in range(16)]
    for j in range(16):
        if oversize[j]:
            for i in range(16):
                if not oversize[i]:
                    fmap[i][j] = 1.0 / n_under
        else:
            fmap[j][j] = 1.0
    return {"torque": torque, "power": torque * speed, "fragmentation_map": np.array(fmap)}


def whiten_cone(zone_hardness_mass, speed, k1=0.25, k2=0.5, k3=2.3, k_oversize=1.0,
                k_undersize=0.1):
    """Whiten's crusher model: p = (I - C)(I - B C)^-1 f, B uniform to finer classes."""
    c = np.zeros(16)
    for k, d in enumerate(D):
        if k == 0 or d <= k1:
            c[k] = 0.0
        elif d >= k2:
            c[k] = 1.0
        else:
            c[k] = 1.0 - ((k2 - d) / (k2 - k1)) ** k3
    b = np.zeros((16, 16))
    for j in range(1, 16):
        b[:j, j] = 1.0 / j
    fmap = (np.eye(16) - np.diag(c)) @ np.linalg.inv(np.eye(16) - b @ np.diag(c))
    torque = float(np.dot(k_undersize + (k_oversize - k_undersize) * c, zone_hardness_mass))
    return {"torque": torque, "power": torque * speed, "fragmentation_map": fmap}


def mill(charge_mass, speed, speed_setpoint, **overrides):
    """Mill outputs at the current speed (paper's breakage, classifier and torque models)."""
    p = {**MILL_DEFAULTS, **overrides}
    m_gr = sum(charge_mass)
    m_tot = p["m0"] + m_gr
    m_gra = sum(m for d, m in zip(D, charge_mass) if d >= p["d_gr_a"] * (1 - 1e-9))
    x = speed / p["omega_crit"]
    theta = math.sqrt(1 - x ** 4) if x < 1 else 0.0
    mu_gra = p["k_gr_a"] * theta * m_gra * x / m_gr if m_gr > 0 else 0.0
    tau_a = mu_gra * m_gr * p["g"] * p["r_mill"]
    tau_dr = p["mu_dr"] * m_tot * p["g"] * p["r_mill"]
    tau_acc = m_tot * p["r_mill"] ** 2 * (speed_setpoint - speed) / p["speed_time_constant"]
    tau = tau_dr + tau_acc + tau_a
    d50 = float(sizes.d_passing(np.array(charge_mass), 0.5)) if m_gr > 0 else 0.0
    tau0 = p["mu_dr"] * p["m0"] * p["g"] * p["r_mill"]
    activity = (tau_a * speed / (tau0 * p["omega_crit"])) ** 2
    rate, escape = [], []
    for k, d in enumerate(D):
        e_imp = p["impact_energy"] * (math.e - math.exp(1 - d50 / d)) * d / p["d_gr"]
        e_brk = p["breakage_energy"] / (1 + (d / p["d_gr"]) ** 0.25)
        rate.append(0.0 if k == 0 else p["k_gr"] * e_imp / e_brk * activity)
        z = p["k_cl"] * (d / p["d_cl"] - 1)
        escape.append(0.0 if z > 700 else p["k_esc"] / (1 + math.exp(z)))
    daughter = [[1.0 / j if i < j else 0.0 for j in range(16)] for i in range(16)]
    return {"breakage_rate": np.array(rate), "daughter_fraction": np.array(daughter),
            "escape_rate": np.array(escape), "speed": speed, "torque_drive": tau_dr,
            "torque_acceleration": tau_acc, "torque_active": tau_a, "torque": tau,
            "power": tau * speed, "d50": d50}


def mill_explicit_step(class_mass, hardness, rate, daughter, escape, dt):
    """The paper's forward-Euler update of one particle's class masses (mass-conserving D)."""
    new = list(class_mass)
    escaped = 0.0
    for j in range(16):
        broken = rate[j] / hardness * class_mass[j] * dt
        leaving = escape[j] * class_mass[j] * dt
        new[j] -= broken + leaving
        escaped += leaving
        for i in range(16):
            new[i] += daughter[i][j] * broken
    return new, escaped
