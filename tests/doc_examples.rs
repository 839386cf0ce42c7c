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
