"""The estimation engine (render, features, learned Jacobian, LM) and the RQ job entry."""
