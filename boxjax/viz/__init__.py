"""Figures (`plots`: mass distributions, episodes, the force map, evaluations) and animations (`animate`:
an episode as a GIF or MP4, seen from above). They read arrays and configs only."""
