"""The flag's record: gross errors flagged, flagged registrations that were fine."""

from pelvicnav.studies.flags import flag_counts, flag_line


def test_flag_counts_per_registration():
    rows = [
        # case a: one bone 6 mm off, flagged -> a gross error, flagged
        {"case_id": "a", "error_mm": 0.2, "converged": False},
        {"case_id": "a", "error_mm": 6.0, "converged": False},
        # case b: fine, flagged -> a false alarm (flags as CSV text)
        {"case_id": "b", "error_mm": 0.3, "converged": "False"},
        # case c: 5 mm off, not flagged -> a missed gross error
        {"case_id": "c", "error_mm": 5.0, "converged": True},
        # case d: fine, not flagged; case e: no answer (NaN) -> gross
        {"case_id": "d", "error_mm": 0.1, "converged": "True"},
        {"case_id": "e", "error_mm": float("nan"), "converged": False},
    ]
    c = flag_counts(rows, "error_mm")
    assert c == {"registrations": 5, "gross": 3, "gross_flagged": 2, "flagged": 3,
                 "flagged_fine": 1}  # fmt: skip
    assert "3 of 5 registrations had an error over 4 mm, 2 of them flagged" in flag_line(c)
    # several error columns: the worst counts
    two = [{"case_id": "x", "l": 1.0, "r": 4.5, "converged": True}]
    assert flag_counts(two, ["l", "r"])["gross"] == 1
    assert flag_counts(two, ["l", "r"], limit_mm=5.0)["gross"] == 0


def test_implausible_flags_are_counted_where_the_rows_carry_them():
    rows = [
        {"case_id": 0, "error_mm": 20.0, "converged": "False", "implausible": "True"},
        {"case_id": 1, "error_mm": 0.3, "converged": "False", "implausible": "False"},
        {"case_id": 2, "error_mm": 0.2, "converged": "False", "implausible": "True"},
        {"case_id": 3, "error_mm": 9.0, "converged": "False", "implausible": "False"},
        {"case_id": 4, "error_mm": 0.1, "converged": "True", "implausible": "False"},
    ]
    c = flag_counts(rows, "error_mm")
    assert (c["flagged"], c["implausible"], c["implausible_gross"]) == (4, 2, 1)
    assert "2 flagged as implausible" in flag_line(c) and "1 of them with an error" in flag_line(c)
    # rows without the column (older stores, other studies): nothing said of it
    plain = [{k: v for k, v in r.items() if k != "implausible"} for r in rows]
    assert "implausible" not in flag_counts(plain, "error_mm")
    assert "implausible" not in flag_line(flag_counts(plain, "error_mm"))


def test_settled_registrations_are_counted_where_the_rows_carry_them():
    rows = [
        {"case_id": 0, "error_mm": 0.3, "converged": "True", "settled": "True"},
        {"case_id": 1, "error_mm": 6.0, "converged": "True", "settled": "True"},
        {"case_id": 2, "error_mm": 0.2, "converged": "False", "settled": "False"},
        {"case_id": 3, "error_mm": 0.1, "converged": "True", "settled": "False"},
    ]
    c = flag_counts(rows, "error_mm")
    assert (c["settled"], c["settled_gross"], c["gross_flagged"]) == (2, 1, 0)
    assert "2 in question settled by the second opinion" in flag_line(c)
    assert "1 of them with an error over 4 mm" in flag_line(c)
    plain = [{k: v for k, v in r.items() if k != "settled"} for r in rows]
    assert "settled" not in flag_counts(plain, "error_mm")
