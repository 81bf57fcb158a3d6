"""Audit of one exchange run: every kilogram and tracking id accounted for.

A tracking id that entered the stockpile with mass m_in must be found as
m_out (reported onto CV301, server ledger) + m_held (still in the pile,
stockpile summary) = m_in to within ``rel_tol`` (default 1e-9, the
mass-balance bound of every test). Less is *lost*; more, or mass of an id that
never entered, is *duplicated*.
"""

from __future__ import annotations

REL_TOL = 1e-9


def audit(ledger: dict, summary: dict, rel_tol: float = REL_TOL) -> dict:
    """Counts and mass balance from the server ledger and the stockpile summary."""
    entered = {int(k): v for k, v in ledger["entered"].items()}
    left = {int(k): v for k, v in ledger["left"].items()}
    held = {int(k): v for k, v in summary["held"].items()}
    lost, duplicated = [], []
    for tid, m_in in entered.items():
        found = left.get(tid, 0.0) + held.get(tid, 0.0)
        if found < m_in * (1 - rel_tol):
            lost.append(tid)
        elif found > m_in * (1 + rel_tol):
            duplicated.append(tid)
    strangers = (set(left) | set(held)) - set(entered)
    mass_in = float(sum(entered.values()))
    mass_out = float(sum(left.values()))
    mass_held = float(sum(held.values()))
    return {
        "bins_in": int(ledger["bins_in"]),
        "bins_out": int(ledger["bins_out"]),
        "mass_in_kg": mass_in, "mass_out_kg": mass_out, "mass_held_kg": mass_held,
        "mass_balance_rel_error": abs(mass_in - mass_out - mass_held) / mass_in if mass_in else 0.0,
        "tracking_ids_lost": len(lost),
        "tracking_ids_duplicated": len(duplicated) + len(strangers),
        "lost_examples": sorted(lost)[:10],
        "duplicated_examples": sorted(set(duplicated) | strangers)[:10],
        "pending_unacknowledged": int(ledger["pending"]),
        "unsent_reports": int(summary.get("outbox", 0)),
    }
