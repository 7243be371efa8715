"""The service: what crosses process boundaries and the processes around the SLAM core.

Versioned messages (`messages`), zenoh keys, sessions, inboxes and liveliness (`transport`),
the command-line options every service process shares (`service`), the camera publisher and
pose client (`clients`), the multi-machine router (`router`) and the launcher that runs
`dimslam run` as processes (`launch`). It may import the core (`geometry`, `map`, `optim`,
`io`) and the pipeline; the core never imports it.
"""
