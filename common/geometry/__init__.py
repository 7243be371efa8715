"""Geometry: the conventions every other module builds on.

SE(3) on 4x4 tensors and its Lie algebra (`pose`: T_wc, OpenCV axes, `T_<to><from>`; the
only place poses are inverted or converted), the pinhole camera with distortion, projection,
unprojection and frustum tests (`camera`), and the one shape-check helper (`shapes`). It
imports nothing of dimslam but `errors`: anything may import it.
"""
