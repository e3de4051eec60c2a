/* The device kernel (_kernel_cuda.cu) compiled as host C++ and launched thread by thread:
 * how the test suite (tests/core/test_device_emulation.py) and `benchmarks/gpu_check.py
 * --emulate` run the device source on a machine without a GPU. Built at test time with the
 * CPU kernel's flags (mcsm.core.emulation), never installed as part of mcsm.
 *
 * A launch runs every thread of every block in order, one after the other. That is exact for
 * this source: its kernels use no shared memory, no barrier and no floating-point atomic, so
 * no thread reads what another thread of the same launch writes.
 *
 * emu_launch(name, grid, block, args) takes the arguments as cuLaunchKernel does (an array of
 * pointers to each argument's value), so the Python launcher passes the same argument list
 * to the emulation and to CuPy.
 */
#include <cstddef>
#include <cstring>
#include <utility>

struct mk_dim3 {
    unsigned x, y, z;
};
static mk_dim3 blockIdx, blockDim, threadIdx, gridDim;

#define __global__
#define __device__
#define __host__
#define __forceinline__ inline

static inline int atomicOr(int *address, int value) {
    int old = *address;
    *address = old | value;
    return old;
}

#include "_kernel_cuda.cu"

template <typename... A, std::size_t... I>
static void call_with(void (*k)(A...), void **args, std::index_sequence<I...>) {
    k(*static_cast<A *>(args[I])...);
}

template <typename... A>
static void run(void (*k)(A...), unsigned grid, unsigned block, void **args) {
    gridDim.x = grid;
    blockDim.x = block;
    gridDim.y = gridDim.z = blockDim.y = blockDim.z = 1;
    blockIdx.y = blockIdx.z = threadIdx.y = threadIdx.z = 0;
    for (unsigned b = 0; b < grid; b++) {
        blockIdx.x = b;
        for (unsigned t = 0; t < block; t++) {
            threadIdx.x = t;
            call_with(k, args, std::index_sequence_for<A...>{});
        }
    }
}

#define MK_EMU(k) if (std::strcmp(name, #k) == 0) { run(k, grid, block, args); return 0; }

/* 0 when the kernel exists and ran, -1 for an unknown name */
extern "C" int emu_launch(const char *name, unsigned grid, unsigned block, void **args) {
    MK_EMU(mk_d_joint_sums)
    MK_EMU(mk_d_joint_gain)
    MK_EMU(mk_d_joint_apply)
    MK_EMU(mk_d_transform)
    MK_EMU(mk_d_meanrot_lanes)
    MK_EMU(mk_d_meanrot_finish)
    MK_EMU(mk_d_canon_check)
    return -1;
}
