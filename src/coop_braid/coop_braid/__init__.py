"""BRAID (thesis app. E): the binary hyper-redundant camera mast: stage and chain kinematics,
inverse kinematics over the 2^(3n) leg states, and the power-line carrier that addresses its
actuators."""
