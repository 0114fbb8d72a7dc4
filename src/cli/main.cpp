#include <cstdio>
int main() { std::puts("tether"); return 0; }
