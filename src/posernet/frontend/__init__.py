"""Image front end: ROI proposals, keypoint matching, box matching, initial relative poses."""
