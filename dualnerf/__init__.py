"""DualNeRF model library: fields, rendering, annealing, consistency, editors, encoders, metrics, scenes.

Imports nothing from `pipeline` or `stages`; usable on its own."""
