// A block of image columns as one GCC/Clang vector: the widest register the build targets (64 bytes with AVX-512,
// 32 with AVX2, 16 with the x86-64 baseline's SSE2; gsmsdr_ns/_cpp_ext.py picks the flags), so that a kernel's
// running sums stay in registers. Header-only, included by each op's single source file.
#pragma once

#include <algorithm>
#include <cstdint>

#if defined(__AVX512F__)
#define GSMSDR_VECTOR_BYTES 64
#elif defined(__AVX2__)
#define GSMSDR_VECTOR_BYTES 32
#else
#define GSMSDR_VECTOR_BYTES 16
#endif

namespace gsmsdr_vec {

template <typename S> struct Block {
    typedef S type __attribute__((vector_size(GSMSDR_VECTOR_BYTES)));
    static constexpr int64_t n = GSMSDR_VECTOR_BYTES / sizeof(S);  // values per block
    // Unaligned load of n values.
    static type load(const S *p) {
        type v;
        __builtin_memcpy(&v, p, sizeof v);
        return v;
    }
    // Store the first count (<= n) values.
    static void store(S *p, type v, int64_t count) {
        S tmp[n];
        __builtin_memcpy(tmp, &v, sizeof v);
        std::copy(tmp, tmp + count, p);
    }
    static S sum(type v) {
        S tmp[n];
        __builtin_memcpy(tmp, &v, sizeof v);
        S acc = 0;
        for (int64_t i = 0; i < n; ++i) acc += tmp[i];
        return acc;
    }
};

// The most values a block holds (16 floats with AVX-512): slack that block loads past a row's end may read.
constexpr int64_t MAX_BLOCK = 16;

}  // namespace gsmsdr_vec
