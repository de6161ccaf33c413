/* The clock tree: 8 MHz HSE -> PLL -> 168 MHz SYSCLK, APB1 42 MHz, APB2 84 MHz, 48 MHz for USB. */
#ifndef FW_CLOCK_H
#define FW_CLOCK_H

void clock_init(void);

#endif
