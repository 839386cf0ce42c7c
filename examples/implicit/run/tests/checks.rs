//! Tests that call gradients live here: a test binary links them, so its
//! package (`run/`) is built with the autodiff flag. Keep the code thin:
//! call functions of the program crate.

#[test]
fn the_checks_pass_and_the_fit_recovers_the_conductivities() {
    starter::run().unwrap();
}
