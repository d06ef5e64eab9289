"""Element kernels of the Lifted Curls model: pure NumPy, batch-first, no PETSc, no MPI.

One module per energy, each with ``energy``, ``gradient`` and ``hessian`` side by side:

========  ==============================  ======================  =====================
module    positions ``x``                 rest quantity           stiffness
========  ==============================  ======================  =====================
stretch   (n, 2, 3): x_i, x_{i+1}         rest length  (n,)       k_s = E A / Lbar
bend      (n, 3, 3): x_{i-1}, x_i, x_{i+1} rest angle   (n,)       k_b = E I / l_i
twist     (n, 4, 3): x_i .. x_{i+3}        rest twist   (n,)       k_t = G J / Lbar_mid
========  ==============================  ======================  =====================

``energy -> (n,)``, ``gradient -> (n, k, 3)``, ``hessian(..., filter=) -> (n, 3k, 3k)``
in vertex-major order (row ``3*v + c`` is coordinate ``c`` of local vertex ``v``).
Rest quantities and stiffnesses are arrays of shape (n,) or scalars. ``filter`` is one of
:data:`FILTERS`:

* ``"none"``: the exact Hessian;
* ``"analytic"``: the closed-form eigen-filter of SPEC section 3 (no eigensolver);
* ``"numerical"``: batched dense eigendecomposition of the same reduced Hessian the
  analytic filter works on, negative eigenvalues clamped to 0 (the paper's baseline).

Every kernel validates its input (shape, finiteness, zero-length edges) and raises
``ValueError`` naming the first offending element. Degenerate geometry has documented
rules (see each module and ``docs/elements.md``).
"""

from lc_petsc.elements.common import FILTERS
from lc_petsc.errors import ElementError
from lc_petsc.elements import stretch, bend, twist, weights

__all__ = ["FILTERS", "ElementError", "stretch", "bend", "twist", "weights"]
