"""``gopre-view`` (also ``pipeline-view``): a finished (or running) episode in a web 3D viewer (viser), with the goal
drawn by the user and scored by the same GO-PRE strategy the sweeps use. An edge package: the core
never imports it."""
