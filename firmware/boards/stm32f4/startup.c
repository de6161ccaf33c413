/* Reset handler and vector table of the STM32F405/407 (RM0090 §10.2, Table 61: 82 peripheral IRQs).
 * Every handler is a weak alias of default_handler, so a board defines only those it uses. */
#include <stdint.h>

#include "vectors.h"

extern uint32_t _sidata, _sdata, _edata, _sbss, _ebss, _estack;
int main(void);

void default_handler(void)
{
    for (;;)
        ;   /* an unexpected exception: stop here, where a debugger shows it */
}

#define WEAK(name) void name(void) __attribute__((weak, alias("default_handler")))
WEAK(nmi_handler);
WEAK(hardfault_handler);
WEAK(memmanage_handler);
WEAK(busfault_handler);
WEAK(usagefault_handler);
WEAK(svc_handler);
WEAK(debugmon_handler);
WEAK(pendsv_handler);
WEAK(systick_handler);
WEAK(exti1_handler);

#define N_IRQ 82
typedef void (*vector)(void);

/* The IRQ slots this firmware may use; the rest fall through to default_handler. */
__attribute__((section(".isr_vector"), used)) static const vector vectors[16 + N_IRQ] = {
    [0] = (vector)(uintptr_t)&_estack,
    [1] = reset_handler,
    [2] = nmi_handler,
    [3] = hardfault_handler,
    [4] = memmanage_handler,
    [5] = busfault_handler,
    [6] = usagefault_handler,
    [11] = svc_handler,
    [12] = debugmon_handler,
    [14] = pendsv_handler,
    [15] = systick_handler,
    [16 + 7] = exti1_handler,
};

void reset_handler(void)
{
    for (uint32_t *src = &_sidata, *dst = &_sdata; dst < &_edata;)
        *dst++ = *src++;
    for (uint32_t *dst = &_sbss; dst < &_ebss;)
        *dst++ = 0;
    main();
    for (;;)
        ;
}
