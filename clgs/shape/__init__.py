"""Statistical shape models of anatomy: the template (:mod:`.template`), the shape model (PCA of
velocity fields) and density atlas (:mod:`.model`), diffeomorphic registration
(:mod:`.registration`), the model builder (:mod:`.builder`), the shape-guided initialisation of
Gaussians on a template (:mod:`.initialise`), the Gaussian set bound to a shape model
(:mod:`.gaussian_set`) and the shape and atlas priors of a fit (:mod:`.priors`).

May import: :mod:`clgs.fit`, :mod:`clgs.ops`, :mod:`clgs.reference`, :mod:`clgs.mesh`,
:mod:`clgs.io`, :mod:`clgs.geometry`. Not methods, anatomies or the CLI.
"""
