//! End-to-end tests of Forja through the simulator.
