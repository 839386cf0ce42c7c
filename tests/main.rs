use diffsim::op::*;
use diffsim::problems::burgers::*;
use diffsim_solvers::burgers::*;

#[test]
fn spike() {
    let cfg = Burgers1d::p1(16);
    let x = p1_initial(&cfg);
    let w: Vec<f64> = (0..16).map(|i| (i as f64 * 0.7).cos()).collect();
    let (a, _) = BurgersEnzyme(cfg).vjp_new(&x, &[], &w);
    let (b, _) = BurgersHand(cfg).vjp_new(&x, &[], &w);
    let (c, _) = FiniteDiff::new(BurgersHand(cfg)).vjp_new(&x, &[], &w);
    for i in 0..16 { println!("{} {} {}", a[i], b[i], c[i]); }
    let t = BurgersEnzyme(cfg).jvp_new(&x, &[], &w, &[]);
    let t2 = FiniteDiff::new(BurgersHand(cfg)).jvp_new(&x, &[], &w, &[]);
    for i in 0..16 { println!("{} {}", t[i], t2[i]); }
}
