"""The fits' objectives on the OpenCL device: parameters in, loss and gradient out, with the
model's bases, the render and the loss images in device buffers that live across evaluations.
The numpy objectives in fitting.recipes stay the reference they are tested against."""
