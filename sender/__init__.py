"""The camera host: capture, tracking, pose and lift, appearance classification, packing."""
