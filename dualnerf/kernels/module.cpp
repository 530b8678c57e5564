#include <torch/extension.h>

#include "kernels.h"

PYBIND11_MODULE(TORCH_EXTENSION_NAME, module) {
  module.def("encode_forward", &encode_forward, "fused dense-grid + plane feature look-ups");
  module.def("encode_forward_pair", &encode_forward_pair, "encode_forward for two fields' tables at once");
  module.def("interleave_pair", &interleave_pair, "two fields' tables as one (cells, 4) table each");
  module.def("encode_backward", &encode_backward, "gradients of encode_forward w.r.t. the tables");
  module.def("field_inference", &field_inference, "look-ups and MLPs of one field or the fused dual field");
  module.def("ray_samples", &ray_samples, "proposal intervals and their occupancy per ray (the render sampler)");
  module.def("adam_step", &adam_step, "one Adam step on one tensor, optionally skipping zero gradients");
  module.def("adam_step_touched", &adam_step_touched, "adam_step (skip zero) on the touched chunks of a gradient buffer");
  module.def("zero_touched", &zero_touched, "zero the flagged chunks of a gradient buffer and the flags");
  module.def("encode_backward_into", &encode_backward_into, "encode_backward into persistent buffers, flagging touched chunks");
  module.def("mlp_inference", &mlp_inference, "a field's MLPs on given features (no autograd)");
  module.def("occupied_samples", &occupied_samples, "a render's occupied sample points, flat index, ray and ray offsets");
  module.def("composite_rays", &composite_rays, "a render's colour and opacity per ray from its evaluated samples");
  module.def("vector_path_available", &vector_path_available, "the AVX-512 look-up and MLP paths can run on this CPU");
  module.def("amx_path_available", &amx_path_available, "field_inference's bf16 MLPs can run on AMX tiles here");
}

