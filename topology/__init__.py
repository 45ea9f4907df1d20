"""flocktrack topology (floor 2): who hears whom.

``topology.graph`` holds the pure graph functions (range adjacency, Laplacian, connectivity,
Chen et al.'s Hₚ = Lₚ + Bₚ and λ₀) and the periodic switching schedules.
"""
