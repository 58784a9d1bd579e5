"""Scene constraints (thesis 2.4): named conditions on whole scene trees; docs/constraints.md.

Each kind is a class with a vectorised `margin(batch)`: one number per tree of a batch, >= 0
when the tree satisfies the constraint, the farther below 0 the worse the violation.
Structural kinds read only the tree's shape (types and parents); pose kinds read poses too.
`ssgc.constraints.build` turns a grammar document's `constraints:` section into them.
"""

from ssgc.constraints.base import Constraint, NodeBatch, satisfied
from ssgc.constraints.pose import Clearance, InsideBox, Upright
from ssgc.constraints.structural import Children, Count, LongestChain

__all__ = [
    "Children",
    "Clearance",
    "Constraint",
    "Count",
    "InsideBox",
    "LongestChain",
    "NodeBatch",
    "Upright",
    "satisfied",
]
