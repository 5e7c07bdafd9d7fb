"""Fingertip-object contact (paper Sec. 3.1-3.4): laws, geometry, and the fingertip interaction."""
