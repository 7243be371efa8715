"""The map: the neural implicit field, its renderer and its mesh.

Feature grids plus the MLP decoder (`field`), volume rendering of depth and colour along
camera rays (`render`), and marching cubes over the observed part of the scene (`mesh`).
It may import `geometry` and the top-level helpers (`options`, `errors`); never `optim`,
`net` or `eval`.
"""
