//! NumPy `.npy` reader and writer (the IncEventGS N×4 float layout and structured arrays).
