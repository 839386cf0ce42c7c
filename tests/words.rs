//! `words`: choices suggested for typos, parser messages in plain words,
//! user values shortened.

use diffsim::words::{ECHO, closest, plain, plain_with_key, unknown};

#[test]
fn typos_get_the_nearest_choice_and_others_the_list() {
    let choices = ["small", "published"];
    assert_eq!(closest("publish", &choices), Some("published"));
    assert_eq!(closest("smal", &choices), Some("small"));
    assert_eq!(closest("nothing-like-it", &choices), None);
    assert_eq!(unknown("setup", "publish", &choices), "unknown setup `publish`; did you mean `published`?");
    assert_eq!(unknown("setup", "zzz", &choices), "unknown setup `zzz`; expected one of small, published");
    // A huge value is not echoed whole.
    let long = "x".repeat(10 * ECHO);
    assert!(unknown("setup", &long, &choices).len() < 3 * ECHO);
}

#[test]
fn parser_messages_read_as_plain_words_with_their_key() {
    let (key, text) = plain("invalid type: floating point `0.5`, expected usize\nin `grid.n`");
    assert_eq!(key.as_deref(), Some("grid.n"));
    assert!(!text.contains("invalid type") && text.contains("0.5"), "{text}");
    assert!(plain_with_key("invalid type: floating point `0.5`, expected usize\nin `grid.n`").starts_with("`grid.n`: "));
    // Without a key the message stays a message.
    assert_eq!(plain("something went wrong").0, None);
}
