"""Matrix Lie groups: SO(2), SE(2), SO(3) and SE(3).

Conventions (shared by every group and by the rest of eqsmooth):

- Each element stores one parameter array with any number of leading batch axes:
  `SO2.unit_complex` `(cos, sin)`, `SE2.unit_complex_xy` `(cos, sin, x, y)`,
  `SO3.wxyz` (quaternion, scalar first), `SE3.wxyz_xyz` `(qw, qx, qy, qz, x, y, z)`.
  The dtype of the parameters (float32 or float64) is preserved by every operation.
- Tangent vectors of SE(2) and SE(3) put the translation part first, then the
  rotation: `(vx, vy, omega)` and `(vx, vy, vz, wx, wy, wz)`.
- `g @ h` composes (apply `h` first), `g @ points` acts on points.
- Perturbations are on the right: `x (+) delta = x @ exp(delta)` and
  `y (-) x = log(x^-1 @ y)`.
- The right Jacobian `Jr(xi)` satisfies `exp(xi + delta) ~= exp(xi) @ exp(Jr(xi) @
  delta)`; the left Jacobian is `Jl(xi) = Jr(-xi)`, with
  `exp(xi + delta) ~= exp(Jl(xi) @ delta) @ exp(xi)`.
- `g.jlog()` is `d log(g @ exp(delta)) / d delta` at `delta = 0`, that is
  `Jr(log(g))^-1`.
- `g.adjoint()` is the matrix `Ad(g)` with `exp(Ad(g) @ xi) = g @ exp(xi) @ g^-1`.

`exp`, `log`, `jlog` and the Jacobians have finite, correct values and derivatives
at angle zero (Taylor series selected without leaking `nan` into gradients) and near
angle `pi` (`atan2`-based logarithm). The logarithm ignores the norm of the rotation
parameters, so slightly unnormalized elements give sensible results.
"""

from ._base import (
    AbstractLieGroup as AbstractLieGroup,
    AbstractRigidMotion as AbstractRigidMotion,
)
from ._se2 import SE2 as SE2
from ._se3 import SE3 as SE3
from ._so2 import SO2 as SO2
from ._so3 import SO3 as SO3
