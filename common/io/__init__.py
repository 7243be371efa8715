"""Input and output: frames in, trajectories out.

One reader per dataset layout behind one protocol (`datasets/`: TUM, Replica, EuRoC,
7-Scenes, image folders, videos, live cameras; a new layout is one small class there), the
built-in synthetic scene the project renders itself (`synth`), and TUM trajectory files
(`trajectory`). It may import `geometry`; never `map`, `optim`, `net` or `eval`.
"""
