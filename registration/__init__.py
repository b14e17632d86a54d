"""Place recognition, image-pair relative pose and RGB-D / point-cloud registration (ICP). Uses `kernels` only."""
