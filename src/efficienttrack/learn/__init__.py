"""Learning: the networks, the closed-loop dynamics model g_θ, the adjustment policy π_φ, training and checkpoints."""
