"""Where ITK lives: images, transforms, manifests, the common frame, memberships, the
pipelines' output folders, the content-keyed cache, and the deformation measures taken on a
transform sampled on a grid (plausibility). Everything that reads, writes or samples an ITK
object is here; :mod:`itk_nrreval.measures` works on the numpy arrays this folder hands it.
"""

__all__: list[str] = []
