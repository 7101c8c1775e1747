"""gopre: goal-oriented active 3D reconstruction (GO-PRE) pipeline."""
