"""The parser: the most probable parse trees of a scene by mixed-integer optimisation
(docs/parsing.md).

Also callable: `ssgc.parse(grammar, scene, top=1, method="auto", time_limit=None)` is
`ssgc.api.parse`, the `top` most probable distinct trees of `scene` as `ssg parse` finds them.
"""
