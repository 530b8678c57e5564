#include <torch/python.h>   // pybind11 and the tensor casters, without all of libtorch's C++ API (torch/extension.h)

#include "kernels.h"

#include <atomic>

namespace {
std::atomic<int> threads{1};
}

int dualnerf::kernel_threads() { return threads.load(std::memory_order_relaxed); }

// The kernels' thread count (see kernels.h, "Threads"): any count gives the same bits.
void set_threads(int64_t n) {
  TORCH_CHECK(n >= 1, "set_threads: at least one thread");
  threads.store(static_cast<int>(n), std::memory_order_relaxed);
}

// A kernel entry point called with denormals flushed (kernels.h, "Denormals") and the caller's mode
// restored on return.
template <typename R, typename... Args>
auto flushed(R (*kernel)(Args...)) {
  return [kernel](Args... args) -> R {
    dualnerf::FlushDenormals flushed;
    return kernel(std::forward<Args>(args)...);
  };
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, module) {
  module.def("set_threads", &set_threads, "the number of threads the kernels use (the results do not depend on it)");
  module.def("get_threads", &dualnerf::kernel_threads, "the number of threads the kernels use");
  module.def("encode_forward", flushed(&encode_forward), "fused dense-grid + plane feature look-ups");
  module.def("encode_forward_pair", flushed(&encode_forward_pair), "encode_forward for two fields' tables at once");
  module.def("interleave_pair", flushed(&interleave_pair), "two fields' tables as one (cells, 4) table each");
  module.def("interleave_pair_into", flushed(&interleave_pair_into), "interleave_pair into existing tables");
  module.def("encode_backward", flushed(&encode_backward), "gradients of encode_forward w.r.t. the tables");
  module.def("field_inference", flushed(&field_inference), "look-ups and MLPs of one field or the fused dual field");
  module.def("ray_samples", flushed(&ray_samples), "proposal intervals and their occupancy per ray (the render sampler)");
  module.def("adam_step", flushed(&adam_step), "one Adam step on one tensor, optionally skipping zero gradients");
  module.def("adam_step_touched", flushed(&adam_step_touched), "adam_step (skip zero) on the touched chunks of a gradient buffer");
  module.def("zero_touched", flushed(&zero_touched), "zero the flagged chunks of a gradient buffer and the flags");
  module.def("encode_backward_into", flushed(&encode_backward_into), "encode_backward into persistent buffers, flagging touched chunks");
  module.def("mlp_train_forward", flushed(&mlp_train_forward), "a field's MLPs for training: outputs and saved activations");
  module.def("mlp_train_backward", flushed(&mlp_train_backward), "the backward of mlp_train_forward (thread-count independent sums)");
  module.def("mlp_inference", flushed(&mlp_inference), "a field's MLPs on given features (no autograd)");
  module.def("occupied_samples", flushed(&occupied_samples), "a render's occupied sample points, flat index, ray and ray offsets");
  module.def("composite_rays", flushed(&composite_rays), "a render's colour and opacity per ray from its evaluated samples");
  module.def("vector_path_available", &vector_path_available, "the AVX-512 look-up and MLP paths can run on this CPU");
  module.def("amx_path_available", &amx_path_available, "field_inference's bf16 MLPs can run on AMX tiles here");
}

