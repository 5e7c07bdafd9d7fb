"""Kinematics of a three-finger Shadow-like hand: URDF model, forward kinematics, Jacobian and WDLS IK."""
