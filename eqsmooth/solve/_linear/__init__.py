"""The linear floor: the normal operator of a linearisation and the lineax
solvers of it (block-tridiagonal, dense, sparse, CG), and the choice of one."""
