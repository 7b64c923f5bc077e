"""SLAM's mapping side: the backend that densifies, keeps keyframes, optimises the map over a window
of them and publishes map versions, and the optimisers it uses."""
