//! Embedded deformation: the graph (Sumner, Schmid, Pauly 2007), its energies with analytic
//! Jacobians, a batch Gauss-Newton / Levenberg-Marquardt solver on block-sparse normal equations
//! (faer sparse Cholesky, symbolic factorisation reused), and the decoupled two-step solver of
//! MIS-SLAM. A plain library: the `deformation.batch` and `deformation.decoupled` nodes wrap it.

// The Jacobian and block code indexes several arrays with one index (Kronecker layouts): explicit
// index loops are the clearer form there.
#![allow(clippy::needless_range_loop)]

mod assemble;
pub mod decoupled;
pub mod engine;
mod evaluate;
pub mod field;
pub mod graph;
pub mod knn;
pub mod node;
pub mod observe;
mod pairs;
mod priors;
pub mod problem;
mod residuals;
mod sampling;
mod schur;
pub mod solver;
pub mod system;

pub use decoupled::{Boundary, DecoupledInfo, DecoupledParams, DecoupledSolver};
pub use engine::{Engine, SolverKind};
pub use field::DistanceField;
pub use graph::{Binding, EdGraph, GraphParams, Sampling};
pub use problem::{
    Correspondence, FieldJacobian, Intrinsics, Method, ModelPoints, ModelSubset, Problem, Robust,
    Scan, SolverParams, Weights,
};
pub use solver::{Info, SolveSet, Solver};
