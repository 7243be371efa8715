"""Optimization: the losses and the window objective that tracking and mapping minimize.

Patch warping, SSIM, smoothness and render terms (`losses`), the window objective that
combines them over a window of frames (`objective`), and the window optimizer with the
frame state it works on (`window`). It may import `geometry` and `map`; never `net` or
`eval`. The tracking and mapping steps themselves live in their process packages
(`dimslam.tracker`, `dimslam.mapper`).
"""
