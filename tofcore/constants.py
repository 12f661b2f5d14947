"""Physical constants shared by every stage (a leaf: it imports nothing)."""

SPEED_OF_LIGHT_M_S = 299_792_458.0
"""c in vacuum (exact, SI): path length L ↔ delay τ = L / c."""
