//! `memory`: sizes read and written, estimates checked against a budget,
//! overflowing estimates refused.

use diffsim::memory::{MemoryError, check_within, f64s, human, human_up, parse_bytes};

#[test]
fn sizes_parse_in_decimal_and_binary_units_and_bad_ones_are_errors() {
    assert_eq!(parse_bytes("123456").unwrap(), 123_456);
    assert_eq!(parse_bytes("50MB").unwrap(), 50_000_000);
    assert_eq!(parse_bytes("1.5G").unwrap(), 1_500_000_000);
    assert_eq!(parse_bytes("2GiB").unwrap(), 2 << 30);
    assert_eq!(parse_bytes(" 500k ").unwrap(), 500_000);
    for bad in ["", "MB", "12 parsecs", "0", "-5MB", "1e30"] {
        assert!(matches!(parse_bytes(bad), Err(MemoryError::Parse(_))), "{bad:?}");
    }
    assert_eq!(human(999), "999 B");
    assert_eq!(human(48_300_000), "48.3 MB");
    assert_eq!(human(2_100_000_000), "2.10 GB");
    // A suggested budget is at least the need and reads back.
    for need in [1, 999, 56_123_456, 3_456_789_012] {
        let s = human_up(need);
        assert!(parse_bytes(&s).unwrap() >= need, "{need} → {s}");
    }
}

#[test]
fn estimates_are_checked_against_the_budget_and_overflows_refused() {
    assert_eq!(f64s(&[10, 10]), Some(800));
    assert_eq!(f64s(&[u64::MAX, 2]), None);
    assert!(check_within(u64::MAX, "a field", "10 values", Some(80), None).is_ok());
    let over = check_within(1000, "a field", "a 1000³ grid", Some(8_000_000_000), Some("a smaller grid".into())).unwrap_err();
    assert!(matches!(over, MemoryError::OverBudget { .. }));
    assert!(over.to_string().contains("a field") && over.to_string().contains("a smaller grid"), "{over}");
    assert!(matches!(check_within(u64::MAX, "a field", "", None, None), Err(MemoryError::Overflow { .. })));
}
