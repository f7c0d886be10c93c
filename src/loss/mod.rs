//! Kernels of the SLAM losses that torch runs slowly on two CPU cores: [`blur`], the separable
//! Gaussian filter of the SSIM term. The losses themselves stay in torch (`evgs.slam.loss`).

pub mod blur;
