"""Posterior quantities of a solution: marginal covariances and log-determinants;
built on the linear floor."""
