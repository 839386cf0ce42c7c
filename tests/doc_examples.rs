//! The doc examples that call generated gradients are marked `ignore`
//! (doctests are built without fat LTO, which Enzyme needs); their code runs
//! here instead, verbatim.

mod lib_rs {
    use diffsim::op::{Operator, OperatorExt};

    struct Square {
        n: usize,
    }
    impl Operator for Square {
        fn n_in(&self) -> usize {
            self.n
        }
        fn n_out(&self) -> usize {
            self.n
        }
    }
    fn square(op: &Square, x: &[f64], _p: &[f64], y: &mut [f64]) {
        for i in 0..op.n {
            y[i] = x[i] * x[i];
        }
    }
    diffsim::differentiable!(Square => square);

    #[test]
    fn crate_root_example() {
        let (dx, _) = Square { n: 2 }.vjp_new(&[1.0, 3.0], &[], &[1.0, 1.0]);
        assert_eq!(dx, vec![2.0, 6.0]);
    }
}

mod differentiable_macro {
    use diffsim::op::{Operator, OperatorExt};

    struct Scale {
        n: usize,
    }
    impl Operator for Scale {
        fn n_in(&self) -> usize {
            self.n
        }
        fn n_out(&self) -> usize {
            self.n
        }
        fn n_params(&self) -> usize {
            1
        }
    }
    fn scale(op: &Scale, x: &[f64], p: &[f64], y: &mut [f64]) {
        for i in 0..op.n {
            y[i] = p[0] * x[i] * x[i];
        }
    }
    diffsim::differentiable!(Scale => scale);

    #[test]
    fn macro_example() {
        let op = Scale { n: 3 };
        let (dx, dp) = op.vjp_new(&[1.0, 2.0, 3.0], &[2.0], &[1.0, 1.0, 1.0]);
        assert_eq!(dx, vec![4.0, 8.0, 12.0]);
        assert_eq!(dp, vec![14.0]);
    }
}

/// docs/own-solver.md quotes the templates of `diffsim new`
/// (`examples/starter`, `examples/implicit`) between `// ANCHOR: name` and `// ANCHOR_END: name`
/// lines; each quoted block must equal its region, and every region must be
/// quoted, so the page cannot drift from the code the test command builds
/// and runs.
#[test]
fn own_solver_page_quotes_the_template() {
    let root = env!("CARGO_MANIFEST_DIR");
    let read = |path: &str| std::fs::read_to_string(format!("{root}/{path}")).unwrap_or_else(|e| panic!("{path}: {e}"));
    let page = read("docs/own-solver.md");
    let mut quoted: Vec<String> = Vec::new();
    let mut rest = page.as_str();
    while let Some(at) = rest.find("<!-- quote: ") {
        rest = &rest[at + "<!-- quote: ".len()..];
        let marker = &rest[..rest.find(" -->").expect("an unclosed quote marker")];
        let (path, anchor) = marker.split_once('#').expect("quote markers read PATH#ANCHOR");
        let start = rest.find("```rust\n").expect("a rust block after the marker") + "```rust\n".len();
        let len = rest[start..].find("```").expect("a closed block");
        let block = &rest[start..start + len];
        let file = read(path);
        let open = format!("// ANCHOR: {anchor}\n");
        let a = file.find(&open).unwrap_or_else(|| panic!("{path} has no anchor {anchor}")) + open.len();
        let b = a + file[a..].find(&format!("// ANCHOR_END: {anchor}")).unwrap_or_else(|| panic!("{path}: {anchor} is not closed"));
        assert_eq!(block, &file[a..b], "docs/own-solver.md quotes {marker} differently from the file");
        quoted.push(marker.to_string());
        rest = &rest[start + len..];
    }
    for path in
        ["examples/starter/solver/src/lib.rs", "examples/starter/src/lib.rs", "examples/implicit/solver/src/lib.rs", "examples/implicit/src/lib.rs"].iter()
    {
        let file = read(path);
        for line in file.lines().filter_map(|l| l.trim().strip_prefix("// ANCHOR: ")) {
            assert!(quoted.contains(&format!("{path}#{line}")), "{path}#{line} is not quoted in docs/own-solver.md");
        }
    }
    assert!(quoted.len() >= 13, "{quoted:?}");
}

/// Every relative link of the README and the docs pages points to a file
/// that exists (pages move; links must follow).
#[test]
fn links_between_the_pages_resolve() {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
    let mut pages = vec![root.join("README.md")];
    for entry in std::fs::read_dir(root.join("docs")).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().is_some_and(|e| e == "md") {
            pages.push(path);
        }
    }
    let mut checked = 0;
    for page in &pages {
        let text = std::fs::read_to_string(page).unwrap();
        let mut rest = text.as_str();
        while let Some(at) = rest.find("](") {
            rest = &rest[at + 2..];
            let target = &rest[..rest.find(')').unwrap_or(0)];
            let target = target.split('#').next().unwrap_or("");
            if target.is_empty() || target.contains("://") || target.contains(' ') {
                continue;
            }
            let file = page.parent().unwrap().join(target);
            assert!(file.exists(), "{}: the link to {target} points to nothing", page.display());
            checked += 1;
        }
    }
    assert!(checked > 30, "only {checked} links found");
}
