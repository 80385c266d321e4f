"""Statistical shape models of anatomy: the template, the shape model (PCA of velocity fields)
and density atlas, diffeomorphic registration, the model builder and the shape-guided
initialisation of Gaussians on a template.

May import: :mod:`clgs.ops`, :mod:`clgs.reference`, :mod:`clgs.mesh`, :mod:`clgs.io`,
:mod:`clgs.geometry`. Not fit, methods, anatomies or the CLI.
"""
