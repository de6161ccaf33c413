#include "ring.h"

void fw_ring_init(fw_ring *r)
{
    atomic_init(&r->head, 0u);
    atomic_init(&r->tail, 0u);
}

bool fw_ring_push(fw_ring *r, const fw_sample *s)
{
    uint32_t head = atomic_load_explicit(&r->head, memory_order_relaxed);
    uint32_t tail = atomic_load_explicit(&r->tail, memory_order_acquire);
    if (head - tail >= FW_RING_CAPACITY)
        return false;
    r->slot[head % FW_RING_CAPACITY] = *s;
    atomic_store_explicit(&r->head, head + 1u, memory_order_release);
    return true;
}

bool fw_ring_pop(fw_ring *r, fw_sample *out)
{
    uint32_t tail = atomic_load_explicit(&r->tail, memory_order_relaxed);
    uint32_t head = atomic_load_explicit(&r->head, memory_order_acquire);
    if (head == tail)
        return false;
    *out = r->slot[tail % FW_RING_CAPACITY];
    atomic_store_explicit(&r->tail, tail + 1u, memory_order_release);
    return true;
}

uint32_t fw_ring_fill(fw_ring *r)
{
    return atomic_load_explicit(&r->head, memory_order_acquire) -
           atomic_load_explicit(&r->tail, memory_order_acquire);
}
