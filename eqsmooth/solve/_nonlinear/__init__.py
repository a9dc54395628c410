"""The nonlinear floor: the optimistix least-squares solvers on graphs, their
adjoints and the `least_squares` entry point; built on the linear floor."""
