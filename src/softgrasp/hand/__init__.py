"""A multi-finger hand: its URDF (urdf), forward kinematics and Jacobian (kinematics), the WDLS step
(wdls), the clamped WDLS descent (descent), one finger's IK (ik) and the palm placement (placement)."""
