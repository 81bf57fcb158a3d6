"""The monitor's alarm book: dead band, states, acknowledgement, restart."""

from __future__ import annotations

import pytest

from cosim.errors import ValidationError
from monitor.alarms import AlarmBook
from monitor.config import load_monitor_config


@pytest.fixture
def book(tmp_path):
    """50 t capacity, level high at 60 % with a 4 % dead band (clears at or below 56 %)."""
    path = tmp_path / "monitor.toml"
    path.write_text("[stockpile]\ncapacity_t = 50\n[alarms]\nlevel_high_pct = 60\n"
                    "level_low_pct = 0\nlevel_deadband_pct = 4\ngrade_low_pct = 25\n"
                    "grade_high_pct = 75\ngrade_deadband_pct = 1\n")
    return AlarmBook(load_monitor_config(path))


def _row(time_s, held_t, grade=0.5):
    return {"time_s": time_s, "held_mass_kg": 1000.0 * held_t, "grade": grade}


def _states(book):
    return [(o["seq"], o["id"], o["state"]) for o in book.occurrences]


def test_a_level_hovering_at_the_limit_raises_one_alarm(book):
    # 59-61 % around the 60 % limit, never down to 56 %: one occurrence, still active
    for k, held in enumerate([29.0, 30.5, 29.5, 30.5, 28.5, 30.2, 28.1]):
        book.check_row(_row(float(k), held))
    assert _states(book) == [(1, "level_high", "ACTIVE_UNACK")]
    assert book.occurrences[0]["raised_s"] == 1.0
    assert book.occurrences[0]["value"] == pytest.approx(61.0)
    # at the clearing value (56 % = 28 t) it clears
    book.check_row(_row(7.0, 28.0))
    assert _states(book) == [(1, "level_high", "CLEARED_UNACK")]
    assert book.occurrences[0]["cleared_s"] == 7.0
    assert book.summary()["active"] == 0 and book.summary()["unacknowledged"] == 1


def test_without_a_dead_band_every_crossing_is_an_alarm(tmp_path):
    path = tmp_path / "monitor.toml"
    path.write_text("[stockpile]\ncapacity_t = 50\n[alarms]\nlevel_high_pct = 60\n"
                    "level_deadband_pct = 0\n")
    book = AlarmBook(load_monitor_config(path))
    for k, held in enumerate([29.0, 30.5, 29.5, 30.5, 28.5]):
        book.check_row(_row(float(k), held, 0.01))  # inside the default grade band
    assert _states(book) == [(1, "level_high", "CLEARED_UNACK"),
                             (2, "level_high", "CLEARED_UNACK")]


def test_low_alarms_clear_above_the_limit_plus_the_dead_band(book):
    grades = [0.30, 0.249, 0.255, 0.259, 0.26]  # grade low 25 %, clears at >= 26 %
    for k, grade in enumerate(grades):
        book.check_row(_row(float(k), 20.0, grade))
    assert _states(book) == [(1, "grade_low", "CLEARED_UNACK")]
    assert (book.occurrences[0]["raised_s"], book.occurrences[0]["cleared_s"]) == (1.0, 4.0)


def test_an_empty_pile_leaves_the_grade_alarms_alone(book):
    book.check_row(_row(0.0, 20.0, 0.8))
    book.check_row({"time_s": 1.0, "held_mass_kg": 0.0, "grade": None})
    assert _states(book) == [(1, "grade_high", "ACTIVE_UNACK")]


def test_acknowledgement_states_who_and_when(book):
    book.check_row(_row(0.0, 35.0))
    book.check_row(_row(1.0, 36.0))
    acknowledged = book.acknowledge(1, " Ana Operator ")
    assert [o["seq"] for o in acknowledged] == [1]
    occurrence = book.occurrences[0]
    assert (occurrence["state"], occurrence["acked_by"], occurrence["acked_s"]) == \
        ("ACTIVE_ACK", "Ana Operator", 1.0)
    assert occurrence["acked_at"].endswith("Z")
    with pytest.raises(ValueError, match="acknowledged by 'Ana Operator'"):
        book.acknowledge(1, "Ben")
    book.check_row(_row(2.0, 20.0))  # acknowledged, then cleared: closed
    assert _states(book) == [(1, "level_high", "CLEARED")]
    # raised and cleared before anyone looked: waits for an acknowledgement
    book.check_row(_row(3.0, 35.0))
    book.check_row(_row(4.0, 20.0))
    book.check_row(_row(5.0, 10.0, 0.9))
    assert _states(book) == [(1, "level_high", "CLEARED"), (2, "level_high", "CLEARED_UNACK"),
                             (3, "grade_high", "ACTIVE_UNACK")]
    assert [o["seq"] for o in book.acknowledge("all", "Ben")] == [2, 3]
    assert _states(book) == [(1, "level_high", "CLEARED"), (2, "level_high", "CLEARED"),
                             (3, "grade_high", "ACTIVE_ACK")]
    assert book.summary()["unacknowledged"] == 0 and book.summary()["active"] == 1


@pytest.mark.parametrize("seq, operator, field", [
    (1, "", "operator"), (1, "   ", "operator"), (1, None, "operator"), (1, "x" * 65, "operator"),
    (1, "tab\there", "operator"), ("one", "Ana", "seq"), (True, "Ana", "seq"),
])
def test_bad_acknowledgements_name_the_field(book, seq, operator, field):
    book.check_row(_row(0.0, 35.0))
    with pytest.raises(ValidationError) as refused:
        book.acknowledge(seq, operator)
    assert refused.value.field == field


def test_unknown_occurrence(book):
    with pytest.raises(LookupError, match="no alarm occurrence 9"):
        book.acknowledge(9, "Ana")


def test_a_restart_clears_the_old_runs_alarms(book):
    book.check_row(_row(100.0, 35.0))
    book.check_row(_row(101.0, 35.0))
    book.check_row(_row(2.0, 35.0))  # the clock went back: a new run, still above the limit
    assert _states(book) == [(1, "level_high", "CLEARED_UNACK"), (2, "level_high", "ACTIVE_UNACK")]
    assert (book.occurrences[0]["cleared_by"], book.occurrences[0]["cleared_s"]) == \
        ("restart", 2.0)
    assert book.occurrences[1]["raised_s"] == 2.0
