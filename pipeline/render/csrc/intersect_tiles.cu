// Tile intersections at a fixed capacity on the GPU: what render/intersections.py builds in
// tensors, in one kernel and one radix sort. Each Gaussian writes its own entries from its
// offset in the inclusive cumulative count (as gsplat's intersect_tile kernel does), entries
// past the capacity are dropped, the rest of the buffer keeps the padding key; the sort reads
// only the bits a key uses (image | tile | depth), as gsplat's does. No host read anywhere, so
// the call can be recorded in a CUDA graph.
#include <c10/cuda/CUDAException.h>
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>
#include <cub/device/device_radix_sort.cuh>
#include <torch/extension.h>

namespace {

__global__ void fill_entries(
    const float *__restrict__ means2d,  // [I N, 2] pixels
    const int32_t *__restrict__ radii,  // [I N, 2] pixels, 0: not drawn
    const float *__restrict__ depths,   // [I N]
    const int64_t *__restrict__ ends,   // [I N] inclusive cumulative entry counts
    const int64_t flat, const int64_t n, const float tile_size, const int32_t tiles_x, const int32_t tiles_y,
    const int32_t tile_bits, const int64_t capacity,
    int64_t *__restrict__ keys,   // [capacity], padding already written
    int32_t *__restrict__ ids) {  // [capacity]
    const int64_t idx = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
    if (idx >= flat) return;
    const int32_t rx = radii[2 * idx], ry = radii[2 * idx + 1];
    if (rx <= 0 || ry <= 0) return;
    int64_t entry = idx == 0 ? 0 : ends[idx - 1];
    if (entry >= capacity) return;
    const float cx = means2d[2 * idx] / tile_size, cy = means2d[2 * idx + 1] / tile_size;
    const float reach_x = static_cast<float>(rx) / tile_size, reach_y = static_cast<float>(ry) / tile_size;
    const int32_t x0 = static_cast<int32_t>(fminf(fmaxf(floorf(cx - reach_x), 0.0f), static_cast<float>(tiles_x)));
    const int32_t y0 = static_cast<int32_t>(fminf(fmaxf(floorf(cy - reach_y), 0.0f), static_cast<float>(tiles_y)));
    const int32_t x1 = static_cast<int32_t>(fminf(fmaxf(ceilf(cx + reach_x), 0.0f), static_cast<float>(tiles_x)));
    const int32_t y1 = static_cast<int32_t>(fminf(fmaxf(ceilf(cy + reach_y), 0.0f), static_cast<float>(tiles_y)));
    const int64_t image = (idx / n) << (32 + tile_bits);
    const int64_t depth_bits = static_cast<int64_t>(static_cast<uint32_t>(__float_as_int(depths[idx])));
    for (int32_t y = y0; y < y1; ++y) {
        for (int32_t x = x0; x < x1; ++x) {
            if (entry >= capacity) return;
            keys[entry] = image | (static_cast<int64_t>(y * tiles_x + x) << 32) | depth_bits;
            ids[entry] = static_cast<int32_t>(idx);
            ++entry;
        }
    }
}

}  // namespace

std::vector<torch::Tensor> intersect_tiles_fixed(
    torch::Tensor means2d, torch::Tensor radii, torch::Tensor depths, torch::Tensor ends, int64_t tile_size,
    int64_t tiles_x, int64_t tiles_y, int64_t tile_bits, int64_t image_bits, int64_t capacity, int64_t padding_key) {
    TORCH_CHECK(means2d.is_cuda() && means2d.scalar_type() == torch::kFloat32, "means2d: float32 on CUDA");
    TORCH_CHECK(radii.scalar_type() == torch::kInt32, "radii: int32");
    TORCH_CHECK(depths.scalar_type() == torch::kFloat32, "depths: float32");
    TORCH_CHECK(ends.scalar_type() == torch::kInt64, "ends: int64");
    const c10::cuda::CUDAGuard guard(means2d.device());
    cudaStream_t stream = c10::cuda::getCurrentCUDAStream();
    const int64_t flat = depths.numel();
    const int64_t n = depths.size(-1);
    auto keys = torch::full({capacity}, padding_key, ends.options());
    auto ids = torch::zeros({capacity}, radii.options());
    if (flat > 0) {
        const int threads = 256;
        const int64_t blocks = (flat + threads - 1) / threads;
        fill_entries<<<blocks, threads, 0, stream>>>(
            means2d.contiguous().data_ptr<float>(), radii.contiguous().data_ptr<int32_t>(),
            depths.contiguous().data_ptr<float>(), ends.contiguous().data_ptr<int64_t>(), flat, n,
            static_cast<float>(tile_size), tiles_x, tiles_y, tile_bits, capacity, keys.data_ptr<int64_t>(),
            ids.data_ptr<int32_t>());
        C10_CUDA_KERNEL_LAUNCH_CHECK();
    }
    auto keys_sorted = torch::empty_like(keys);
    auto ids_sorted = torch::empty_like(ids);
    const int end_bit = static_cast<int>(32 + tile_bits + image_bits);
    size_t temp_bytes = 0;
    cub::DeviceRadixSort::SortPairs(
        nullptr, temp_bytes, keys.data_ptr<int64_t>(), keys_sorted.data_ptr<int64_t>(), ids.data_ptr<int32_t>(),
        ids_sorted.data_ptr<int32_t>(), capacity, 0, end_bit, stream);
    auto temp = torch::empty({static_cast<int64_t>(temp_bytes)}, keys.options().dtype(torch::kUInt8));
    cub::DeviceRadixSort::SortPairs(
        temp.data_ptr(), temp_bytes, keys.data_ptr<int64_t>(), keys_sorted.data_ptr<int64_t>(),
        ids.data_ptr<int32_t>(), ids_sorted.data_ptr<int32_t>(), capacity, 0, end_bit, stream);
    return {keys_sorted, ids_sorted};
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
    m.def("intersect_tiles_fixed", &intersect_tiles_fixed, "tile intersections at a fixed capacity, sorted");
}
