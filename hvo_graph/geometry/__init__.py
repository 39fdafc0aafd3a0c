"""Pure geometry: camera model, rotations, discrete (H_d) and continuous (H_c) homographies."""
