#include "clock.h"

#include "board.h"
#include "regs.h"

/* PLL (RM0090 §6.3.2): VCO in = HSE / M = 1 MHz, VCO out = 1 MHz * N = 336 MHz, SYSCLK = VCO / P = 168 MHz,
 * USB = VCO / Q = 48 MHz. */
#define PLL_M (HSE_HZ / 1000000u)
#define PLL_N 336u
#define PLL_P 2u
#define PLL_Q 7u

void clock_init(void)
{
    RCC_CR |= RCC_CR_HSEON;
    while (!(RCC_CR & RCC_CR_HSERDY))
        ;
    RCC_PLLCFGR = PLL_M | (PLL_N << 6) | ((PLL_P / 2u - 1u) << 16) | (1u << 22) /* HSE */ | (PLL_Q << 24);
    RCC_CR |= RCC_CR_PLLON;
    while (!(RCC_CR & RCC_CR_PLLRDY))
        ;
    /* 5 wait states at 168 MHz and 3.3 V, prefetch, instruction and data caches */
    FLASH_ACR = 5u | (1u << 8) | (1u << 9) | (1u << 10);
    /* AHB / 1, APB1 / 4, APB2 / 2, then switch SYSCLK to the PLL */
    RCC_CFGR = (5u << 10) | (4u << 13);
    RCC_CFGR |= 2u;
    while (((RCC_CFGR >> 2) & 3u) != 2u)
        ;
}
