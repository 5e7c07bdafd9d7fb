"""The paper's experiments: compression test (Fig. 8-9), indentation (Fig. 10-11), grasp."""
