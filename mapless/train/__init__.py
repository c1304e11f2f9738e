"""Training: the A3C loss, the meta-learning inner loop and the trainers."""
